"""radaredge."""
