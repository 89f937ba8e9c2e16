"""Multi-seed experiment suites that reproduce the paper's tables (stats, plots, table1/2/3)."""
