"""Train-accident scene reconstruction workbench."""
__version__ = "0.1.0"
