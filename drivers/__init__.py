"""drivers package of dh2rt."""
