"""The ground floor: what every layer may use (cancellation, memory limits, child processes, compiled loops, BLAS threads)."""
