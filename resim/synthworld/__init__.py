"""The synthetic driving world's simulator: road network and scenery (world.py, fork.py), renderer
(render.py), ego vehicle and drivers (drivers.py), infraction score (score.py).

A leaf package: it imports nothing of resim's own (numpy and OpenCV only), so both the pipeline's
``resim synth`` (which writes the world's episodes in the real layouts) and training's closed-loop
evaluation (which drives a policy in the true world) can use it."""
