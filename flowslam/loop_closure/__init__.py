"""Loop closure: place recognition (Scan Context) and geometric verification (ICP)."""
