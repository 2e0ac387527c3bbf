"""The estimator's REST models (`focustrack_client.models`) in the domain's words, and back.

The one translation between the API's JSON models, which lab software and the
scheduler send and the estimator serves, and the domain's types
(`focustrack_core.domain`), which the strategies and the scan plan compute with:
`to_domain` reads API models into domain values, `to_api` writes domain values as
API models. The estimator and the scheduler both use it; the client stays
httpx, pydantic and the OpenTelemetry API only.

The API models are the users' contract: their defaults (`ZRangePolicy`,
`SlideCreate`) are the product's, and `to_domain.default_settings` gives them to
code that builds a slide without a request (benchmarks, tests).
"""
