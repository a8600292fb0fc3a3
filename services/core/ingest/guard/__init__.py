"""What guards the service against a hostile or broken upload: confinement, archive and size limits,
mesh checks, and loading in a bounded process."""
