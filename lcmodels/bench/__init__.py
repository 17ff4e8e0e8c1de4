"""The benchmark: a suite of scenarios with their ceilings and floors, sealed test episodes evaluated
through one path that appends to a committed ledger, and the tables ``lc-bench`` prints.

- :mod:`lcmodels.bench.ledger`: the ledger of sealed test evaluations;
- :mod:`lcmodels.bench.run`: drivers resolved from specs, cells run or found again;
- :mod:`lcmodels.bench.table`: the suite table (Markdown and JSON) with its statistics.
"""
