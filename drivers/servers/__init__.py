"""Protocol servers of the simulated machine (apart from the gateway's clients)."""
