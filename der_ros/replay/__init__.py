"""ROS-free replay core: uniform (DQN), prioritized (PER) and double experience replay (DER).

``factory.make_replay(cfg, obs_shape, obs_dtype, batch_size, seed)`` builds the buffer a
``config.ReplayConfig`` asks for; every buffer has the ``base.ReplayBuffer`` interface and
returns ``base.Batch`` tuples; ``factory.load_replay(path)`` restores one saved with ``save``.
Import-light on purpose (``config`` must not load numba): import the module you need.
"""
