"""The ``dm2`` command line (click)."""
