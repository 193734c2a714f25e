"""On top of the library: the command line, the demo, reports, plots, the meshcat views and dataset files."""
