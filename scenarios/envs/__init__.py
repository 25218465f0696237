"""Gymnasium environments over the bench (the only place that imports gymnasium)."""
