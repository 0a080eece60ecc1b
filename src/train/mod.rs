pub mod adam;
