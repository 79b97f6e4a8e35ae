"""Link-model profiles (TOML), shipped as package data: ``--comm NAME``."""
