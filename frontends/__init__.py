"""Frontends: per-scan motion estimation (and, for flow frontends, per-point flow)."""
