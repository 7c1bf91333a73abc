"""resim: driving world models from heterogeneous video.

The distribution holds five top-level packages:

* ``shards``    the WebDataset shard format (schema, writer, manifest, reader, CLI);
* ``labeling``  driving commands from optical flow and from trajectories;
* ``pipelines`` Ray jobs: sources -> clips -> labels -> balance -> latents -> shards;
* ``training``  world model, Video2Reward, IDM, sampler, metrics, launcher;
* ``resim``     this package: the ``resim`` CLI, shared config helpers and the demo.
"""
__version__ = "0.1.0"
