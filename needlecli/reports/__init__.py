"""Tables and plots, built from results files only."""

import needlecli.reports.consistency  # noqa: F401  (registers the consistency table and the NEES plot)
import needlecli.reports.control  # noqa: F401  (registers the closed loops' table)
import needlecli.reports.imaging  # noqa: F401  (registers the imaging sensors' plot and table)
from needlecli.reports import real, seed000_001, seed003, seed004  # noqa: F401  (register the seeds' and real data's tables and plots)
from needlecli.reports.tables import TABLES, write_table

__all__ = ["TABLES", "write_table"]
