"""progress feature of the API."""
