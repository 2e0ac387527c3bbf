"""Python code generated from the wire schemas in proto/focustrack/v1 (do not edit the *_pb2 files).

Regenerate with `make proto` (`python proto/generate.py`); a test fails when
these files are out of date.
"""
