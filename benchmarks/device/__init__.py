"""The GPU and many-core checks, in one run on a machine with a GPU and many cores."""
