"""The focus service: focus metrics and peak fitting (pure), served over Zenoh and REST."""
