"""File formats of the pipeline: images and masks, COLMAP models, PLY point clouds, atomic output."""
