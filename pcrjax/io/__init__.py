"""Files: scene TOML, CSV time series, run outputs."""
