"""The dashboard designer: plan a spec over stored spaces, its distributions and a few previews."""
