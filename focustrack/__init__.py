"""FocusTrack: predictive autofocus for automated slide-scanning microscopes."""

__version__ = "0.1.0"
