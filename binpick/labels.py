"""Point labels beside the instances (>= 0), as the training, the scoring and the labelled
captures read them."""

# Known to be no part: a rendered distractor or bin rim, a capture's point beyond its bin.
NOT_A_PART = -1
# Left out of the loss and the scoring: a capture's point the cell cannot explain (input, not target).
IGNORE = -2
