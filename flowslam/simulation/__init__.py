"""LiDAR simulator: procedural towns, moving actors, ray-cast sensors, exact ground truth."""
