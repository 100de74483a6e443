"""Figures (PNG) of every study. Each module imports pyplot only inside its functions and never
switches matplotlib's backend, so importing them is cheap and safe anywhere."""
