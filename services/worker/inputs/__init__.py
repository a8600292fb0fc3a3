"""What tasks are computed from, kept between tasks: job rows, the loaded space, its curvature, photos."""
