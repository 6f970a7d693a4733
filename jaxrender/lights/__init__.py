"""Light sources: spot lights (cone, falloff, projected light map), the sun, environment maps
with importance sampling. One private module per kind; public names re-exported here."""
