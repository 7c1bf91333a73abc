"""The synthetic driving world (issue 3): road network, renderer, drivers, infraction score, writers."""
