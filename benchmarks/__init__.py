"""Speed and memory benchmarks (scripts, not timed tests); see README.md."""
