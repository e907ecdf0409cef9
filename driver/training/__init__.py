"""What drives one training run: its planner, its loop, checkpoints, summaries, curriculum, the
learner keeper and start-up timing."""
