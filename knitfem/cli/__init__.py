"""The ``knitfem`` command: its commands, the -knit_ options and the scenes."""
