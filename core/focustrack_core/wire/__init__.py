"""The Zenoh edge shared by every service: key expressions, sessions and the z-stack codec.

The message schemas are in proto/focustrack/v1 (generated code in focustrack_core.v1);
proto/README.md documents the key space for subscribers in any language.
"""
