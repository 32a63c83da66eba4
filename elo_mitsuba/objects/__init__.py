"""Generated test objects of known shape: the corrugated sheet (Sec. 4.2) and the melt plate (Fig. 3).

Each module builds its object's height or mesh exactly and regenerates the shipped asset in
``scenes_xml/meshes/``; the tests hold the shipped files to the generators.
"""
