"""Sub-commands of the `piezo-stage` CLI: one module each, with `add_arguments(parser)` and
`run(args) -> int`."""

# Nothing to import from here: piezo_stage.cli loads each sub-command module by name, on demand
# (so that `piezo-stage gains` does not pay for rclpy or the identification).
__all__: list[str] = []
