"""What is knitted: stitch patterns (charts by name or file, knitting-machine
programs in knitout), the stitch pattern's geometric template and the fabric
it becomes (yarns as B-spline control polygons, their crossings, held
points)."""
