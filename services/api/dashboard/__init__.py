"""dashboard feature of the API."""
