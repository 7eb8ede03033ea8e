"""Start graphs: the YAML launcher, its domains, scenario runs and live tuning."""
