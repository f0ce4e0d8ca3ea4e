"""Import every command module so that it registers on the app."""

from needlecli.cli import compare, evaluate, listing, log, simulate, sweep, validate  # noqa: F401
