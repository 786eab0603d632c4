"""Sub-commands of the `piezo-stage` CLI: one module each, with `add_arguments(parser)` and
`run(args) -> int`."""
