"""A worker's core: stepping its Unity instance, acting, packing rows into segments, counting what
it produced; and the worker's thin Ray shell."""
