"""Tables and plots, built from results files only."""

from needlecli.reports.tables import TABLES, write_table

__all__ = ["TABLES", "write_table"]
