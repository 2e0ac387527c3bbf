"""The estimator service: each slide's Kalman filter behind a durable REST API."""
