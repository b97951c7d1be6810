"""Bundled mixer definitions (TOML data, loaded by bridge.mixing); see README.md here."""
