"""Dataset readers (one class per module) and the format-guessing factory."""
