"""The `shadowopt bench` commands, each writing its table into BENCHMARKS.md (`suite.write_section`):
suite (coarse buffers, quality on the demo and the corpus, solvers, trust), quality_report (the corpus
tables and verdicts), heldout (the held-out scenes), batches, load (the server under concurrent
requests) and security (the hostile corpus against a running server)."""
