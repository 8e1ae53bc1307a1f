"""The contact model: the exact pair potential, the central potential and blend, the sphere hierarchy, and the
BSH potential of body pairs and scenes built from them."""
