"""Import every command module so that it registers on the app."""

from needlecli.cli import evaluate, listing, log, simulate, validate  # noqa: F401
