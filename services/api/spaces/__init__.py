"""spaces feature of the API."""
