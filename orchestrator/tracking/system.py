"""System metrics of a run (CPU, memory, disk, network), under MLflow's `system/` names so that the
MLflow UI shows them in its "System metrics" tab.

MLflow's own collectors (`mlflow.system_metrics.metrics`) sample in a background thread every
`interval_s`; the training loop takes their averages at most once per interval (`take`) and logs
them with its other metrics, through the run's tracker, so that they are spooled like the rest
while the server is away (MLflow's `SystemMetricsMonitor` would write past the spool).
"""

from __future__ import annotations

import logging
import threading
import time

log = logging.getLogger(__name__)

PREFIX = "system/"


class SystemMetrics:
    def __init__(self, interval_s: float = 10.0):
        # Imported here, not with the module: a run that tracks nothing never imports mlflow.
        import psutil
        from mlflow.system_metrics.metrics.cpu_monitor import CPUMonitor
        from mlflow.system_metrics.metrics.disk_monitor import DiskMonitor
        from mlflow.system_metrics.metrics.network_monitor import NetworkMonitor

        self.interval_s = interval_s
        self.monitors = [CPUMonitor(), DiskMonitor(), NetworkMonitor()]
        self.process = psutil.Process()
        self.lock = threading.Lock()
        self.stopped = threading.Event()
        self.last_take = time.monotonic()
        self.collect()  # the first CPU reading starts psutil's interval
        self.thread = threading.Thread(target=self._sample, name="system-metrics", daemon=True)
        self.thread.start()

    def collect(self) -> None:
        with self.lock:
            for m in list(self.monitors):
                try:
                    m.collect_metrics()
                except Exception as e:  # noqa: BLE001 - a collector that fails is dropped, not the run
                    log.warning("system metrics: %s dropped (%s)", type(m).__name__, e)
                    self.monitors.remove(m)

    def _sample(self) -> None:
        while not self.stopped.wait(self.interval_s):
            self.collect()

    def take(self) -> dict[str, float]:
        """The averages since the last take, once per interval (empty in between or before any sample)."""
        now = time.monotonic()
        if now - self.last_take < self.interval_s:
            return {}
        self.last_take = now
        out: dict[str, float] = {}
        with self.lock:
            for m in self.monitors:
                if m.metrics:
                    out.update({PREFIX + k: float(v) for k, v in m.aggregate_metrics().items()})
                    m.clear_metrics()
        if out:
            out[PREFIX + "driver_memory_megabytes"] = self.process.memory_info().rss / 1e6
        return out

    def close(self) -> None:
        self.stopped.set()
        self.thread.join(timeout=self.interval_s + 1)
