"""Result review for the application (stages, flows, the service): MLflow tracking and rerun
recordings. The library never calls either."""
