"""The refiner networks: shared blocks, one module per architecture family, and the registry that builds them by
name (``build_refiner("shallow")``). Importing this package imports no architecture; the registry does on first use."""
