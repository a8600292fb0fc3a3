"""outputs feature of the API."""
