"""Learned scene flow after MambaFlow: model, selective scan, losses, metrics, training."""
