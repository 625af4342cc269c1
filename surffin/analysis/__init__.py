"""Analyses of the method's results.

Diagnostics, sensitivity, uncertainty, evaluation against truth, the paper comparison.
"""
