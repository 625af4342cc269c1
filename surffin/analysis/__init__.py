"""Analyses of the method's results: diagnostics, sensitivity, uncertainty, evaluation against truth, the paper comparison."""
