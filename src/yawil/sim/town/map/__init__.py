"""The static town: layout files (`maps/*.json`) -> lane graph -> routes (`planner`); the geometry handed to the
renderers (`geometry`, `scenery`, `buildings`), the lookup grid (`regions`), pedestrian paths (`walkways`),
and `town.get_town`, which builds all of it once per town."""
