"""Import every command module so that it registers on the app."""

from needlecli.cli import characterize, compare, evaluate, listing, log, simulate, sweep, validate  # noqa: F401
