"""The REST API's routes, one module per tag: slides, scan, maps, strategies, operations."""
