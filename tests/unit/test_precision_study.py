"""scripts/precision_study.py's paired verdicts on rows worked by hand."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest

spec = importlib.util.spec_from_file_location(
    "precision_study", Path(__file__).parents[2] / "scripts" / "precision_study.py"
)
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)


def rows(ratios: dict[str, list[float]]) -> list[dict]:
    out = []
    for s in range(len(next(iter(ratios.values())))):
        base = {"seed": s, "alpha": 1e-4, "beta": 2.0}
        out.append({**base, "precision": "float32", **{k: 1.0 + s for k in study.MEASURES}})
        out.append({**base, "precision": "bfloat16", **{k: (1.0 + s) * ratios[k][s] for k in study.MEASURES}})
    return out


def test_paired_log_ratios_within_the_margins_are_no_change_and_a_shift_is_a_change():
    same = {k: [1.00, 1.01, 0.99, 1.00] for k in study.MEASURES}
    result = study.judge_rows(rows(same))
    assert result["seeds"] == [0, 1, 2, 3]
    for key, m in result["measures"].items():
        # log ratios 0, ±0.00995 (sd 0.00817 over 4 pairs), t(1 - 0.05/6, 3) = 4.857: ± 2.0%, inside ±10%.
        assert m["ratio"] == pytest.approx(1.0, abs=1e-3) and m["verdict"] == "no change", key
        assert m["high"] == pytest.approx(math.exp(4.857 * 0.008165 / 2), abs=2e-4)
    shifted = dict(same, **{"eval/heldout_action_error": [1.30, 1.31, 1.29, 1.30]})
    assert study.judge_rows(rows(shifted))["measures"]["eval/heldout_action_error"]["verdict"] == "changed"
    noisy = dict(same, **{"eval/time_until_fall_mean": [0.7, 1.4, 0.9, 1.2]})
    assert study.judge_rows(rows(noisy))["measures"]["eval/time_until_fall_mean"]["verdict"] == "not resolved"
