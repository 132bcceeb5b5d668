"""``laserrl-report``: the paper's figures and a table of its claims against laserrl's numbers.

``context`` computes what the figures and the table need (lazily, once), ``figures`` is the
registry of figure functions, ``claims`` the table, ``spot`` trains missing models with small
budgets, ``app`` is the Hydra entry point.
"""
