"""hil package of dh2rt."""
