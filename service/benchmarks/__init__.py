"""Benchmarks behind `netpose bench`: accuracy on rendered nets with ground truth, and speed."""
