"""Figures and animations: generic drawing here, one module per method's diagnostics."""
