"""ROS-free DQN learner (paper section 2.1): ``config`` (DQNConfig), ``networks``, ``schedules``,
``optim`` (FlatAdam), ``dqn`` (DQNAgent), and ``online`` (the agent node's stamp-joining core).

Import-light on purpose: import the module you need; ``dqn`` and ``networks`` load torch.
"""
