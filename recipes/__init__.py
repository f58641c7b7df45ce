"""Recipes: typed configs -> make_* builders -> one training loop (see recipes/README.md)."""
