"""Protocol servers of the simulated machine: what the gateway's clients in ``drivers`` talk to."""
