"""Runners that string the library together: the benchmark, the SeqMatchNet ablation and the demo."""
