"""`flightstack sweep`: one experiment over seeds × a grid of mission overrides, in parallel, resumable.

- `plan`: the --set grid, the combinations (seed × grid point) and their stable ids, the recorded plan;
- `execute`: one combination in a worker process (`run_combination`) and the executor loop (a
  ProcessPoolExecutor, or a Dask cluster's executor), writing DIR/runs/<id>.json atomically;
- `stats`: per grid point and mode, statistics over seeds (mean, median, Student-t 95 % CI), ratios,
  ordering fractions, the gain condition;
- `report`: summary.csv, summary.json, the plots and the printed table.
"""
