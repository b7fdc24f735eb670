"""What every benchmark shares: the grid runner (:mod:`.runner`) and the command-line options
(:mod:`.options`)."""
