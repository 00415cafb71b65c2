"""Robust point-set registration: weighted Kabsch, IRLS, RANSAC, covariance."""
