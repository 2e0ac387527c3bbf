"""Quantitative phase from a through-focus stack of intensity images (pure numpy/scipy)."""
