// Test scene for `mvsplat360 pose`: a small still life made for SIFT, seen from all sides.
// Every surface has high-contrast, non-repeating procedural texture so each orbit view has many distinctive
// features; a textured wall at finite distance surrounds it (a sky at infinity gives no parallax).
// Rendered into orbit24/ as assets/pose-test/README.md says.
// No radiosity, area lights or focal blur: about a second per frame at 320x180 on one thread.

#version 3.7;
global_settings { assumed_gamma 1.0 max_trace_level 4 }

// Size of the texture detail: larger is coarser (fewer features, smaller JPEGs).
#ifndef (TS) #declare TS = 2; #end

// The loop circles look_at at this distance and height (scripts/render-povray-scene reads them).
camera {
   location <0, 3.4, -8.5>
   look_at <0, 0.9, 0>
}

light_source { <-20, 30, -25> color rgb 1.1 }
light_source { <25, 22, 18> color rgb 0.8 }
light_source { <0, 40, 0> color rgb 0.4 shadowless }

#declare Matte = finish { ambient 0.25 diffuse 0.75 specular 0.05 }

// Ground: a checker whose two squares carry different non-periodic patterns, so corners are sharp but no two
// tiles look alike.
plane {
   y, 0
   texture {
      pigment {
         checker
         pigment { bozo color_map { [0 rgb <0.05, 0.05, 0.1>] [0.35 rgb <0.9, 0.85, 0.2>]
                                       [0.6 rgb <0.1, 0.4, 0.9>] [1 rgb <1, 1, 1>] } scale 0.9 }
         pigment { bozo turbulence 0.6 octaves 2 color_map { [0 rgb <0.95, 0.2, 0.1>] [0.3 rgb <0.05, 0.05, 0.05>]
                                                   [0.55 rgb <0.2, 0.9, 0.3>] [0.8 rgb <1, 1, 0.9>]
                                                   [1 rgb <0.4, 0.1, 0.6>] } scale 0.35 }
         scale 1.3 * TS
      }
      finish { Matte }
   }
}

// Surrounding wall (open cylinder, seen from inside) with agate bands, leopard spots and large painted numerals.
cylinder {
   <0, -0.1, 0>, <0, 14, 0>, 22 open
   texture {
      pigment { agate agate_turb 0.7 octaves 3 color_map { [0 rgb <0.1, 0.05, 0.3>] [0.25 rgb <1, 0.6, 0.1>]
                                                 [0.5 rgb <0.05, 0.3, 0.1>] [0.75 rgb <0.95, 0.95, 1>]
                                                 [1 rgb <0.6, 0, 0.1>] } scale 2.2 * TS }
      finish { ambient 0.45 diffuse 0.6 }
   }
   texture {
      pigment { leopard color_map { [0 rgbt <0, 0, 0, 1>] [0.55 rgbt <0, 0, 0, 1>]
                                                   [0.6 rgb <0, 0, 0>] [1 rgb <0.02, 0.02, 0.05>] } scale 0.7 * TS }
      finish { ambient 0.45 diffuse 0.6 }
   }
}

#declare Font = "timrom.ttf";
#declare I = 0;
#while (I < 12)
   text {
      ttf Font str(I * 7 + 3, 0, 0) 0.3, 0
      pigment { color rgb <mod(I, 3) / 2, mod(I + 1, 2), 1 - mod(I, 4) / 3> }
      finish { ambient 0.6 diffuse 0.4 }
      scale 2.6
      translate <-1.3, 1.5 + 2.2 * mod(I, 3), -21.5>
      rotate y * (I * 30 + 10)
   }
   #declare I = I + 1;
#end

// The still life, within 3 units of the centre so the objects hide each other differently from each side.
box {
   <-1, 0, -1>, <1, 2, 1>
   texture {
      pigment {
         checker
         pigment { agate octaves 3 color_map { [0 rgb <0.9, 0.1, 0.1>] [0.5 rgb <1, 0.9, 0.6>] [1 rgb <0.1, 0.1, 0.2>] }
                   scale 0.6 }
         pigment { bozo color_map { [0 rgb <0, 0.2, 0.5>] [0.5 rgb <0.95, 0.95, 0.95>] [1 rgb <0.1, 0.5, 0>] }
                   scale 0.8 }
         scale 0.5 * TS
      }
      finish { Matte }
   }
   rotate y * 25
   translate <0.4, 0, 0.3>
}

sphere {
   <0, 1.1, 0>, 1.1
   texture {
      pigment { bozo turbulence 0.8 octaves 2 color_map { [0 rgb <0.05, 0, 0.2>] [0.3 rgb <1, 0.4, 0>]
                                                          [0.5 rgb <1, 1, 0.7>] [0.7 rgb <0, 0.6, 0.7>]
                                                          [1 rgb <0.2, 0, 0>] } scale 0.35 * TS }
      finish { ambient 0.2 diffuse 0.75 specular 0.2 roughness 0.05 }
   }
   translate <-2.3, 0, -0.9>
}

cylinder {
   <0, 0, 0>, <0, 3.2, 0>, 0.55
   texture {
      pigment { marble turbulence 1.2 octaves 3 color_map { [0 rgb <1, 1, 1>] [0.2 rgb <0.1, 0.1, 0.1>]
                                                  [0.5 rgb <0.9, 0.7, 0.1>] [0.8 rgb <0.1, 0.2, 0.8>]
                                                  [1 rgb <1, 1, 1>] } scale 0.7 * TS }
      finish { Matte }
   }
   translate <2.2, 0, -1.4>
}

cone {
   <0, 0, 0>, 0.9, <0, 2.1, 0>, 0.05
   texture {
      pigment { spotted color_map { [0 rgb <0, 0, 0>] [0.3 rgb <0.2, 0.9, 0.2>] [0.6 rgb <1, 1, 1>]
                                    [1 rgb <0.8, 0, 0.5>] } scale 0.25 * TS }
      finish { Matte }
   }
   translate <-0.8, 0, 2.3>
}

torus {
   0.75, 0.28
   texture {
      pigment { wrinkles color_map { [0 rgb <0.1, 0, 0>] [0.4 rgb <1, 0.8, 0>] [0.7 rgb <0.1, 0.3, 1>]
                                     [1 rgb <1, 1, 1>] } scale 0.3 * TS }
      finish { Matte }
   }
   rotate x * 70
   rotate y * -30
   translate <1.9, 1.0, 1.9>
}

text {
   ttf Font "POSE 24" 0.25, 0
   pigment { color rgb <1, 0.95, 0.2> }
   finish { ambient 0.4 diffuse 0.6 }
   scale 0.9
   translate <-1.9, 0.2, -2.7>
   rotate y * 8
}
