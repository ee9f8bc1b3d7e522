"""bop package."""
