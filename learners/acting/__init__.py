"""What a rollout worker acts with, without torch: the policy and image encoders in numpy, and the
factory both sides build a behavior's policy from."""
