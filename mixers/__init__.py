"""Bundled mixer definitions (TOML data, loaded by bridge.mixer); see README.md here."""
