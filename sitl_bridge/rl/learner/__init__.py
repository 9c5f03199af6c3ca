"""The learning algorithm: DQN network and config, replay buffers (uniform, prioritized,
n-step, persisted), input normalizer, exploration, checkpoints and the greedy policy."""
