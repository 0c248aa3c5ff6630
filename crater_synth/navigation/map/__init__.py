"""The landmark map: craters measured in a polar DEM, checked against independent crater lists."""
