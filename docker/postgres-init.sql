-- Run by the postgres image on an empty data volume: the database of MLflow's auth app (its users and
-- permissions), beside the tracking database that POSTGRES_DB creates.
CREATE DATABASE mlflow_auth;
