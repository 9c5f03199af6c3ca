"""Flying a policy: rollouts on fixed reset seeds, greedy evaluation, videos."""
