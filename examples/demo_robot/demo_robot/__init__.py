"""Four small nodes: odometry at a steady rate, a planner that follows it,
a map server that answers, and a lifecycle navigator with an action."""
