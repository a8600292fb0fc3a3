"""The worker process itself: numeric threads, the heap, the compiled kernels and their warm-up."""
