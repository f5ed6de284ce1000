"""bradyscope's product around the measurement library: service, pages, reports, CLI."""
