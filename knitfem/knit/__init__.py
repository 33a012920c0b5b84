"""What is knitted: the stitch pattern's geometric template and the fabric it
becomes (yarns as B-spline control polygons, their crossings, held points)."""
