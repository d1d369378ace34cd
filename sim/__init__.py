"""sim package of dh2rt."""
