"""tools package of dh2rt."""
