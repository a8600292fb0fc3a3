"""workers feature of the API."""
