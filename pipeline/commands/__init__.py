"""The commands of the command line (pipeline/cli.py), one module each, imported only when its command runs: each
defines `add_arguments(parser, command)` and `main(args)`."""
