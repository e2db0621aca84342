"""One module per command-line tool (morph-train, morph-eval, morph-export, ...)."""
