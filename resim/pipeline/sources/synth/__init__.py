"""The synthetic driving world: road network, renderer, drivers, infraction score, writers."""
