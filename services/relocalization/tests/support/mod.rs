pub mod rendered_map;
