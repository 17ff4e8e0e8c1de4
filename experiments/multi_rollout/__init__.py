"""The safety layer scoring each decision by rollouts of several base policies across all its imagined futures."""
