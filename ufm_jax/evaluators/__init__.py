"""Evaluators, one per benchmark family, chosen by name from config or `evaluate.py --bench`."""
