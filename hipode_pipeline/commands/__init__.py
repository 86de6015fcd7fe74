"""CLI command groups, one module each; `hipode_pipeline.cli` assembles them."""
