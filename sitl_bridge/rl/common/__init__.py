"""What every part of the learning side shares: the N-drone env view, atomic writes,
the episode log, action names, progress lines and statistics across seeds."""
