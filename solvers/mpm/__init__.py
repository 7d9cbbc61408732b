"""MLS-MPM solver: soft bodies, plasticine, sand and liquids on a background grid."""
