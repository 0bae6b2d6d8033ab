"""Oracles the bench and the tests share: analytic solutions and the NumPy particle step."""
