"""The `shadowopt bench` commands, each writing its table into BENCHMARKS.md (`output.write_section`):
coarse (coarse buffers), quality (Chong & Gortler's protocol on the demo scene), quality_corpus (the same
on the corpus; its tables and verdicts in corpus_tables, the report pieces in quality_report), solvers
(speed against error, pareto_plot), trust, heldout (the held-out scenes), batches, load (the server
under concurrent requests), security (the hostile corpus against a running server), engine, path,
inspect, throughput and budget. definitions reads configs/benchmarks.json and configs/corpus.json."""
