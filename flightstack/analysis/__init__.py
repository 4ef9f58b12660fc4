"""What a run's recordings say: the error metrics and the paper comparison, loop health, the plots."""
