"""jobs feature of the API."""
