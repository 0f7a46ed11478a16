"""What a result becomes: reports, certificates and their checker, explanations, the viewer."""
