// What the live page imports from its libraries; scripts/vendor-live.sh bundles this (with the
// versions package-lock.json pins) into live-libs.min.js. Add an export here to use more.
export * as THREE from "three";
export { OrbitControls } from "three/addons/controls/OrbitControls.js";
export { CSS2DRenderer, CSS2DObject } from "three/addons/renderers/CSS2DRenderer.js";
export { ViewHelper } from "three/addons/helpers/ViewHelper.js";
export { Lut } from "three/addons/math/Lut.js";
export { default as uPlot } from "uplot";
