"""What a run leaves behind: in-memory time series, the run directory written as the run goes, plots."""
