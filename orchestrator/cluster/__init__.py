"""The cluster topology on one machine, without Docker (`python -m orchestrator.cluster up|down|status|env`): the
command line (`__main__`), the cluster's lifecycle and its record (`topology`), each service started and stopped
(`services`), and the processes under them, each in its own session (`procs`). MLflow's basic-auth app and the
private directories and secret files live in `orchestrator.tracking` (`mlflow_auth`, `secret_files`), which the
tracking server of a parallel sweep uses too.
"""
