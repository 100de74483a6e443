"""Studies, each a ``run_*(config) -> result`` API over the simulation: `reproduce` (the paper's
scenarios), `montecarlo` (robustness over a case distribution), `tuning` (gains by gradient
through the ISE), `unmodeled` (full plant, motor lag, digital control) and `bench` (throughput);
`executors` says where their batches run (this process, or a Dask cluster) and `scaling`
measures the Dask path against one process. Nothing is imported eagerly: import the module you
need."""
