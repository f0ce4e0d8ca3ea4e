"""Tables and plots, built from results files only."""

from needlecli.reports import seed003  # noqa: F401  (registers seed 003's tables and plots)
from needlecli.reports.tables import TABLES, write_table

__all__ = ["TABLES", "write_table"]
