"""What a trained policy does: behaviour classes and summary, candidate rules, rule and
tree policies, distillation, pictures of episodes, training plots."""
