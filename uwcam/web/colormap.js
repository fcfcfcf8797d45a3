// Colour maps as 256-entry lookup tables of packed RGBA (little-endian: 0xAABBGGRR).
// turbo: Google's polynomial approximation of the Turbo colour map (Apache-2.0, A. Mikhailov, 2019).
// deep, thermal: cmocean 3.0.3 (MIT, K. Thyng et al., Oceanography 2016), sampled at 256 levels.

const CMOCEAN = {
  deep: "fdfeccfbfdcbf9fccaf7fbc8f5fac7f3fac6f1f9c5eff8c4edf7c3ebf7c1e9f6c0e7f5bfe5f4bee3f4bde1f3bcdff2bbddf2badbf1b9d9f0b8d7efb7d4efb6d2eeb5d0edb4ceecb3ccecb3caebb2c8eab1c6eab0c4e9afc1e8afbfe7aebde7adbbe6acb9e5acb7e5abb5e4aab2e3aab0e2a9aee2a9ace1a8aae0a8a7e0a7a5dfa7a3dea6a1dda69fdda59cdca59adba598daa496daa494d9a492d8a490d7a48dd7a38bd6a389d5a387d4a385d3a383d3a381d2a37fd1a37dd0a37ccfa37acea378cea376cda375cca373cba371caa370c9a36ec8a36dc7a36bc6a36ac5a469c4a467c3a466c2a465c2a464c1a463c0a462bfa461bea460bda45fbca45ebba45dbaa45cb9a45bb8a45ab7a45ab6a459b4a458b3a458b2a457b1a456b0a456afa455aea355ada354aca353aba353aaa352a9a352a8a351a7a351a6a251a5a250a4a250a3a24fa2a24fa1a24fa0a24e9fa14e9ea14d9da14d9ca14d9ba14c9aa04c99a04b98a04b97a04b96a04a959f4a949f4a939f49929f49919e49909e488f9e488e9e488d9d478c9d478b9d478a9d46899d46889c46879c45869c45859c45849b44839b44829b44819b44809b437f9a437e9a437d9a427c9a427b99427a994279994178994177994176984075984074984073984072984071973f70973f6f973f6e973f6d973f6c963e6b963e6a963e69963e68963e67953e66953e65953e64953e63943e62943e61943e60943e5f933e5e933e5c933e5b933e5a923e59923e58923e57913e56913f55903f54903f538f3f528f3f508e404f8d404e8d404d8c404c8b414b8a414a8941498841488741478541468441458341448142438041427e41417d41407b41407a413f78413e76413d75403c73403c71403b70403a6e3f396c3f386b3f38693e37673e36663d35643d35623d34613c335f3c325d3b325c3b315a3a30583a3057392f55392e54382d52382d51372c4f362b4d362a4c352a4a35294934284734284633274432264332254131254030243e30233d2f223b2f223a2e21392d20372d1f362c1f342b1e332b1d322a1c30291c2f281b2d281a2c",
  thermal: "04233304243504253704253905263b05273d05273f052841052943062945062a47062b49072b4b072c4d072c50082d52082e54092e56092f590a2f5b0b305d0c30600c30620d31650e31670f326a10326c12326f13337214337416337717337a19337c1a347f1c34821e34841f348721348a23348c25348f2734912a33932c33952e339730339933339b35339c37339d39339e3c339f3e349f40349f4234a04435a04635a04736a049369f4b379f4d379f4e389e50399e52399d533a9d553b9d563b9c583c9c593d9b5b3d9b5c3e9a5e3f9a5f3f996040996241986341986542976643976743966944966a45956c45956d46946e4794704794714893724893744992754a92764a92784b91794b917a4c917c4d907d4d907e4e90804e8f814f8f83508f84508e85518e87518e88528d89528d8b538d8c538c8e548c8f548c90558b92558b93568b95568a96578a97578a9958899a58899c59899d59889f5a88a05a87a25b87a35b86a55c86a65c86a85d85a95d84ab5d84ac5e83ae5e83af5f82b15f82b26081b46080b56180b7617fb8627eba627ebb627dbd637cbe637bc0647bc1647ac36579c46578c66677c76676c96775ca6774cc6873cd6872ce6971d06970d16a6fd36a6ed46b6dd66c6cd76c6bd86d6ada6e69db6e68dc6f66de7065df7064e07163e17262e37260e4735fe5745ee6755de7765be8775aea7859eb7958ec7956ed7a55ee7b54ee7d53ef7e52f07f50f1804ff2814ef3824df3834cf4854bf5864af58749f68848f68a47f78b46f78c45f88e44f88f43f99143f99242f99341fa9541fa9640fa983ffb993ffb9b3efb9c3efb9e3efb9f3dfba13dfca33dfca43dfca63cfca73cfca93cfcaa3cfcac3cfcae3cfcaf3cfcb13cfbb23dfbb43dfbb63dfbb73dfbb93efbbb3efbbc3efabe3ffabf3ffac140fac340f9c441f9c641f9c842f8c943f8cb43f8cd44f7ce45f7d045f7d246f6d347f6d547f5d748f5d849f4da4af4dc4bf3dd4bf3df4cf2e14df2e24ef1e44ff1e650f0e851efe951efeb52eeed53edee54edf055ecf256ebf457eaf558eaf759e9f95ae8fa5b",
};

function turbo(t) {
  const r = 0.13572138 + t * (4.6153926 + t * (-42.66032258 + t * (132.13108234 + t * (-152.94239396 + t * 59.28637943))));
  const g = 0.09140261 + t * (2.19418839 + t * (4.84296658 + t * (-14.18503333 + t * (4.27729857 + t * 2.82956604))));
  const b = 0.1066733 + t * (12.64194608 + t * (-60.58204836 + t * (110.36276771 + t * (-89.90310912 + t * 27.34824973))));
  return [r, g, b].map((v) => Math.round(255 * Math.min(1, Math.max(0, v))));
}

function pack(r, g, b, a = 255) {
  return ((a << 24) | (b << 16) | (g << 8) | r) >>> 0;
}

export const COLOUR_MAPS = ["turbo", "deep", "thermal"];

// Near is drawn bright or warm (turbo and thermal reversed; deep already runs from pale to dark):
// what is closest, and most in the way, stands out. The reason colours below are greys and
// purples that none of the maps uses.
const REVERSED = { turbo: true, thermal: true, deep: false };

export function lut(name) {
  const table = new Uint32Array(256);
  if (name in CMOCEAN) {
    const hex = CMOCEAN[name];
    for (let i = 0; i < 256; i++) {
      const c = parseInt(hex.slice(6 * i, 6 * i + 6), 16);
      table[i] = pack((c >> 16) & 255, (c >> 8) & 255, c & 255);
    }
  } else {
    for (let i = 0; i < 256; i++) table[i] = pack(...turbo(i / 255));
  }
  return REVERSED[name] ? table.reverse() : table;
}

// Invalid pixels, drawn by reason (codes as in uwcam.optics.validity.Reason).
export const REASON_COLOURS = {
  1: [96, 96, 96],     // below noise floor: mid grey
  2: [255, 255, 255],  // saturated: white
  3: [70, 110, 140],   // backscatter only (water): murky blue-grey
  4: [120, 60, 130],   // too few channels: purple
  5: [200, 60, 160],   // path out of bounds: magenta
  6: [40, 40, 40],     // the vehicle in view (bracket, skids): near black
};

export function reasonColour(code) {
  const c = REASON_COLOURS[code] || [128, 128, 128];
  return pack(c[0], c[1], c[2]);
}

export function cssColour(packed) {
  return `rgb(${packed & 255}, ${(packed >> 8) & 255}, ${(packed >> 16) & 255})`;
}
