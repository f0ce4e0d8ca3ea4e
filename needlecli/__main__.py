from needlecli.cli.app import run

run()
