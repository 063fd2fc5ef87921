"""captures package."""
