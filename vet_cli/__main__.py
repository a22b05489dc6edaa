from vet_cli.main import cli

cli(prog_name="vet")
