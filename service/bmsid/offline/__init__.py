"""Offline inputs and fits: tester CSV loading, OCV-test fitting (the imperative edges are thin)."""
