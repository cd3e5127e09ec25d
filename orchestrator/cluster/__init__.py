"""The cluster topology on one machine, without Docker (`python -m orchestrator.cluster up|down|status|env`): the
command line (`__main__`), the cluster's lifecycle and its record (`topology`), each service started and stopped
(`services`), MLflow's basic-auth app and the lab's user (`mlflow_auth`), the private directories and secret files
of the state dir (`files`), and the processes under them, each in its own session (`procs`).
"""
