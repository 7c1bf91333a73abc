"""resim: driving world models from heterogeneous video. One import namespace; its folders, in the order data
travels (docs/architecture.md has the layer rules):

* ``resim.media``       video I/O and the encoders (VAE, T5) shared by the pipeline and training;
* ``resim.shards``      the WebDataset shard format (schema, writer, manifest, reader, CLI);
* ``resim.labeling``    driving commands from optical flow and from trajectories;
* ``resim.synthworld``  the synthetic world's simulator (``resim synth``, the closed loops);
* ``resim.pipeline``    Ray jobs: sources -> clips -> labels -> balance -> latents -> shards;
* ``resim.models``      networks and how one is built or loaded: the world DiT, Video2Reward, the IDM, the policy;
* ``resim.diffusion``   noise schedule and levels, losses, DDIM and guidance;
* ``resim.sample``      rollouts, planning and simulation inside a world model;
* ``resim.train``       the training loop, with one task per trainable model;
* ``resim.eval``        metrics and evaluation protocols;
* the face: ``resim.cli``, the config kernel ``resim.config`` and ``resim.demo``.
"""
__version__ = "0.1.0"
