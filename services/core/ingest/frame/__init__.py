"""A scan's frame: which way is up and what unit it is in, detected from its geometry or given."""
