"""One leaf (time interval) of the certificate tree: placement, the stages, their composition."""
