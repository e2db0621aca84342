"""Reports on finished runs: summaries and rankings, plots, videos, the shipped-policy choice."""
