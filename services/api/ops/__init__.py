"""ops feature of the API."""
