"""Losses, miners, the one training loop and its learners (SeqMatchNet, SeqNet, JIST), settings and run state."""
