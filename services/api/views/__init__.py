"""views feature of the API."""
