"""The benchmark: a suite of scenarios with their ceilings and floors, sealed test episodes evaluated
through one path that appends to a committed ledger, and the tables ``lc-bench`` prints.

- :mod:`lcmodels.bench.ledger`: the ledger of sealed test evaluations, its figures derived from its letters;
- :mod:`lcmodels.bench.run`: drivers resolved from specs, cells run or found again;
- :mod:`lcmodels.bench.verify`: ledger lines replayed and their letters compared (``lc-bench --verify``);
- :mod:`lcmodels.bench.table`: the suite table (Markdown and JSON) with its statistics.
"""
