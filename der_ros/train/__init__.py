"""Training: env factory, configs, metrics and the runner behind `der train`."""
