"""rve package."""
