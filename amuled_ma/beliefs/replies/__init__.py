"""An answer read into a belief (reply parsing) and the one check of a valid belief."""
