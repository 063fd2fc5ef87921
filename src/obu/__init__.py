"""obu package."""
