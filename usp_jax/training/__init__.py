"""Training: the configuration, the photo pipeline, the jitted step, the loop and its workdir,
orbax checkpoints. ``usp_jax.training.train.fit`` is the entry point."""
