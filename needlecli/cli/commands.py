"""Import every command module so that it registers on the app."""

from needlecli.cli import characterize, compare, evaluate, fit_em, imports, listing, log, simulate, sweep, validate  # noqa: F401
