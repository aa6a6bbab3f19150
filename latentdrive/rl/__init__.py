"""Q-learning: replay, double DQN, the training loop and its benchmark.

``latentdrive.rl.train.train_policy`` trains a run, through ``latentdrive.rl.learner.Learner``
(replay, updates, checkpoint); ``latentdrive.rl.policy`` builds and
loads networks. The VFAN itself lives in :mod:`latentdrive.models.vfan`.
"""
