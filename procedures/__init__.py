"""The procedure engine, the run store, the CLI, the reports, and the YAML procedures."""
